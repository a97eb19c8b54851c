// The protection of front <-> shard calls (transport_security.h).
#include "server/cluster/transport_security.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/security/credentials.h>
#include <grpcpp/security/server_credentials.h>

#include <fstream>
#include <iterator>

#include "server/http/http_server.h"

namespace oxbow::cluster {

Result<std::string> ReadSmallFile(const std::string& path, std::string_view what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot read " + std::string(what) + " " + path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) return Fail(ErrorCode::kIoError, "cannot read " + std::string(what) + " " + path);
  return text;
}

Result<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const ShardSecurity& security) {
  if (auto ok = security.Check(); !ok) return std::unexpected(ok.error());
  if (!security.tls()) return grpc::InsecureServerCredentials();
  auto cert = ReadSmallFile(security.tls_cert_file, "the TLS certificate");
  if (!cert) return std::unexpected(cert.error());
  auto key = ReadSmallFile(security.tls_key_file, "the TLS private key");
  if (!key) return std::unexpected(key.error());
  grpc::SslServerCredentialsOptions options(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  options.pem_key_cert_pairs.push_back({*key, *cert});
  if (!security.tls_client_ca_file.empty()) {
    auto ca = ReadSmallFile(security.tls_client_ca_file, "the TLS client CA");
    if (!ca) return std::unexpected(ca.error());
    options.pem_root_certs = *ca;
    options.client_certificate_request = GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  return grpc::SslServerCredentials(options);
}

Result<std::shared_ptr<grpc::ChannelCredentials>> MakeChannelCredentials(const FrontSecurity& security) {
  if (!security.tls) return grpc::InsecureChannelCredentials();
  if (security.tls_cert_file.empty() != security.tls_key_file.empty())
    return Fail(ErrorCode::kInvalidArgument, "the front's TLS certificate needs its private key (\"cert\" and \"key\")");
  grpc::SslCredentialsOptions options;
  if (!security.tls_ca_file.empty()) {
    auto ca = ReadSmallFile(security.tls_ca_file, "the TLS CA");
    if (!ca) return std::unexpected(ca.error());
    options.pem_root_certs = *ca;
  }
  if (!security.tls_cert_file.empty()) {
    auto cert = ReadSmallFile(security.tls_cert_file, "the front's TLS certificate");
    if (!cert) return std::unexpected(cert.error());
    auto key = ReadSmallFile(security.tls_key_file, "the front's TLS private key");
    if (!key) return std::unexpected(key.error());
    options.pem_cert_chain = *cert;
    options.pem_private_key = *key;
  }
  return grpc::SslCredentials(options);
}

grpc::Status Authorize(const grpc::ServerContext& context, const std::string& key) {
  if (key.empty()) return grpc::Status::OK;
  const auto& metadata = context.client_metadata();
  const auto found = metadata.find(std::string(kAuthorizationKey));
  if (found == metadata.end()) {
    return {grpc::StatusCode::UNAUTHENTICATED,
            "this shard needs the cluster key (the front's --cluster-key or cluster.json \"key_file\")"};
  }
  const std::string_view value(found->second.data(), found->second.size());
  if (!value.starts_with(kBearerPrefix))
    return {grpc::StatusCode::UNAUTHENTICATED, "the cluster key goes in 'authorization: Bearer KEY'"};
  if (!server::ConstantTimeEquals(std::string(value.substr(kBearerPrefix.size())), key))
    return {grpc::StatusCode::PERMISSION_DENIED, "wrong cluster key"};
  return grpc::Status::OK;
}

}  // namespace oxbow::cluster
