// Helpers shared by the postings tests: bags of words, random corpora, and TF-IDF scores computed from
// the definition to compare an inverted file's against. Header-only; tests only.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <map>
#include <random>
#include <vector>

#include "index/postings/inverted_file.h"

namespace oxbow::index::postings::testing {

inline BagOfWords Bag(std::initializer_list<uint32_t> words) {
  std::vector<uint32_t> w(words);
  return BagOfWords::FromWords(w);
}

// A random bag over `vocab` words with Zipf-like word frequencies, 5..60 features.
inline BagOfWords RandomBag(std::mt19937_64& rng, size_t vocab) {
  std::uniform_int_distribution<int> len(5, 60);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<uint32_t> w;
  const int n = len(rng);
  w.reserve(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) {
    // Inverse-CDF of a truncated power law: frequent low ids, long tail.
    w.push_back(static_cast<uint32_t>(std::min<double>(vocab - 1, std::floor(std::pow(vocab, u(rng)) - 1))));
  }
  return BagOfWords::FromWords(w);
}

// Straightforward dense reference: cosine of tf-idf vectors, computed from the definition, with the
// document frequencies of `statistics` (the corpus itself when null).
inline std::map<uint32_t, double> ReferenceScores(const std::map<uint32_t, BagOfWords>& corpus, const BagOfWords& query,
                                                  size_t vocab, bool sqrt_tf,
                                                  const std::map<uint32_t, BagOfWords>* statistics = nullptr) {
  if (!statistics) statistics = &corpus;
  std::vector<double> df(vocab, 0);
  for (const auto& [id, bag] : *statistics) {
    for (uint32_t w : bag.words) df[w] += 1;
  }
  const double n = static_cast<double>(statistics->size());
  auto t = [&](uint32_t tf) { return sqrt_tf ? std::sqrt(static_cast<double>(tf)) : static_cast<double>(tf); };
  auto vec = [&](const BagOfWords& bag) {
    std::vector<double> v(vocab, 0);
    for (size_t k = 0; k < bag.words.size(); ++k) {
      if (df[bag.words[k]] > 0) v[bag.words[k]] = t(bag.counts[k]) * std::log(n / df[bag.words[k]]);
    }
    return v;
  };
  auto norm = [](const std::vector<double>& v) {
    double s = 0;
    for (double x : v) s += x * x;
    return std::sqrt(s);
  };
  const auto q = vec(query);
  std::map<uint32_t, double> out;
  for (const auto& [id, bag] : corpus) {
    const auto d = vec(bag);
    double dot = 0;
    for (size_t w = 0; w < vocab; ++w) dot += q[w] * d[w];
    const double nq = norm(q), nd = norm(d);
    out[id] = (nq > 0 && nd > 0) ? dot / (nq * nd) : 0.0;
  }
  return out;
}

// Every image `file` lists for `query`, with its score.
inline std::map<uint32_t, double> AllScores(const InvertedFile& file, const BagOfWords& query) {
  ScoreScratch scratch;
  const auto terms = file.QueryVector(query);
  std::map<uint32_t, double> out;
  for (const auto& s : file.Score(terms, 1u << 30, &scratch)) out[s.image] = s.score;
  return out;
}

// `file` after adding n random images numbered from `first` (recorded in *live).
inline InvertedFile AddAll(const InvertedFile& file, std::map<uint32_t, BagOfWords>* live, uint32_t first, size_t n,
                           std::mt19937_64& rng, size_t vocab) {
  std::vector<uint32_t> ids;
  std::vector<const BagOfWords*> bags;
  for (uint32_t i = 0; i < n; ++i) {
    (*live)[first + i] = RandomBag(rng, vocab);
    ids.push_back(first + i);
    bags.push_back(&(*live)[first + i]);
  }
  return file.WithAdded(ids, bags);
}

// The checkpoint form of `file` (InvertedFile::Serialize) as one byte string.
inline std::vector<uint8_t> SerializedBytes(const InvertedFile& file) {
  std::vector<uint8_t> out;
  file.Serialize([&](std::span<const uint8_t> part) { out.insert(out.end(), part.begin(), part.end()); });
  return out;
}

}  // namespace oxbow::index::postings::testing
